"""``perscli apply-persistence``: persistence of earlier exposures on a frame."""

from __future__ import annotations

import logging

import click

from ..detector.settings import (FERMI_PARAMETERS, SETTINGS, ApplyOptions, persistence_param,
                                 preset_default_text)
from ..executor import keep_freed_memory
from .helpers import FILE, PerscliCommand, check_outputs, deprecated_option, file_or, progress_reporter, report_errors
from .options import (FiniteRange, compress_opt, exptime_opt, gain_opt, key_values, no_checksum_opt, output_opt,
                      overwrite_opt, settings_options, units_opt, verbosity_opts, workers_opt)

log = logging.getLogger("perscli")

#: work below this many steps tells a log (stderr not a terminal) nothing: blocks of 64 rows, a full frame's 64
#: are worth telling a log about, a sample frame's 4 are not
PROGRESS_LEAST = 32

#: the defaults, written once (perscli.detector.settings)
D = ApplyOptions()


def setting_option(flag: str, name: str, text: str, metavar: str | None = None):
    """A click option of a persistence setting, typed and ranged by its entry in the table of parameters.

    ``text`` says what the option means on this command's inputs; the allowed values and the defaults
    (the default preset's and any other preset's own) come from the table.
    """
    param = persistence_param(name)
    if param.kind == "choice":
        kind = click.Choice(param.choices)
    elif param.kind == "int":
        kind = click.IntRange(min=param.lo, max=param.hi)
    else:
        kind = click.FloatRange(min=param.lo, max=param.hi, min_open=param.lo_open, max_open=param.hi_open)
    return click.option(flag, name, type=kind, default=None, metavar=metavar,
                        help=f"{text} {preset_default_text(name)}.")


def _power_of_two(ctx, param, value):
    if value is not None and (value < 1 or value & (value - 1)):
        raise click.BadParameter(f"{value} is not one DQ flag: give a power of two (e.g. 1024)")
    return value


@click.command("apply-persistence", cls=PerscliCommand,
               short_help="Add, subtract or predict the persistence of earlier exposures.")
@click.argument("current", metavar="CURRENT", type=FILE)
@click.argument("previous", nargs=-1, required=True, metavar="PREVIOUS...", type=FILE)
@output_opt
@click.option("--law", "law", default=None, metavar="NAME|LAW.yaml|FRAME.fits",
              type=file_or("typical", "pessimistic", "wfc3", "galsim-linear"),
              help="The persistence law: typical or pessimistic (the paper's Table 1), wfc3 (STScI's HST WFC3-IR "
                   "parameters, with the WFC3 pipeline's --time-model middle --combine max --max-previous 0 "
                   "--lookback 16), galsim-linear (GalSim's 8 coefficients), a YAML file (persistence parameters, "
                   "or a detector model as render takes), or a frame perscli rendered (the persistence of the "
                   "model that made it)  [default: typical]")
# the older spelling: --model is the detector model in render and diagnose
@click.option("--model", "model_spec", default=None, hidden=True, type=file_or("typical", "pessimistic", "wfc3",
              "galsim-linear"), callback=deprecated_option("apply-persistence --model", "--law"))
@click.option("--set", "settings", multiple=True, metavar="persistence.KEY=VALUE",
              callback=key_values(effect="persistence"),
              help=f"Override a parameter of the law ({', '.join(FERMI_PARAMETERS)}) or a setting "
                   f"({', '.join(SETTINGS)}), as render's --set does: persistence.gamma=1.1. Repeatable.")
@click.option("--param", "params", multiple=True, hidden=True,
              callback=deprecated_option("apply-persistence --param KEY=VALUE", "--set persistence.KEY=VALUE"))
@settings_options(ApplyOptions, "mode")
# the settings of how the law is applied: type, range and default (per preset) from the one table of
# persistence parameters (perscli.detector.settings.PERSISTENCE_PARAMETERS); None here = the law's own
@setting_option("--time-model", "time_model",
                "exact: integral of the rate over the exposure from the real timestamps; "
                "middle: the rate at the middle of the exposure (of each read's window for a ramp) times "
                "its length, as STScI's WFC3 pipeline; "
                "galsim: galsim.roman.applyPersistence(method='fermi')'s mid-exposure rate")
@setting_option("--combine", "combine",
                "Sum over earlier exposures (the paper, GalSim) or per-pixel maximum (WFC3 pipeline)")
@setting_option("--max-previous", "max_previous",
                "Only the N most recent earlier exposures count (0: all)", metavar="N")
@setting_option("--lookback", "lookback",
                "Ignore earlier exposures that ended more than HOURS before CURRENT starts (0: no limit; "
                "-v names them)", metavar="HOURS")
@settings_options(ApplyOptions, "model_error")
@click.option("--flag-above", type=click.FloatRange(min=0), default=None, metavar="E_PER_S",
              help="Set a DQ bit where the persistence averaged over CURRENT's exposure exceeds E_PER_S "
                   "electrons per second, whatever the units of the data (WFC3's advice: 0.01). A frame "
                   "without DQ gets one.")
@click.option("--dq-bit", type=int, default=None, callback=_power_of_two, metavar="VALUE",
              help=f"The DQ value --flag-above sets, a power of two [default: {D.dq_bit}, a value calwf3 is not known to "
                   "set in WFC3-IR data].")
@click.option("--gap", type=FiniteRange(min=0), default=None, metavar="SECONDS",
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
def apply_persistence(current, previous, output, law, model_spec, settings, params, mode, time_model, combine,
                      max_previous, lookback, model_error, flag_above, dq_bit, gap, units, gain, exptime, compress,
                      overwrite, workers):
    """Add, subtract or predict the persistence of earlier exposures on CURRENT.

    Each earlier exposure (PREVIOUS...) with fluence x electrons releases
    P(x, t) = F(x) (t/1000 s)^-gamma e-/s, t counted from its end (the paper's
    Fermi model, linear below half_well).  The charge added to CURRENT is by
    default the exact integral of P over CURRENT's own exposure window, from EXPSTART/EXPEND,
    MJD-BEG/MJD-END or DATE-OBS + EXPTIME; for a ramp (WFC3-IR raw/ima, or a
    3-D cube with a READTIMES table) it is the integral up to each read.
    Earlier exposures are ordered by their timestamps, not by their order on
    the command line, and only the --max-previous most recent count.

    --law wfc3 follows STScI's WFC3-IR persistence pipeline: its Fermi
    parameters (no linear branch), the rate at the middle of CURRENT, the
    per-pixel maximum over earlier exposures, and those of the last 16 hours;
    each convention can be changed with its own option.

    Fluence of an earlier exposure is its accumulated charge: rate x EXPTIME
    (WFC3 flt), DN x gain, last read minus zeroth read for a raw ramp, the
    last read for a calibrated WFC3 ima.  Non-finite pixels count as zero and
    are reported.  Frames are placed on the detector by LTV1/LTV2 (detector
    pixel = image pixel - LTV): a subarray and a full frame share the pixels
    they both cover, persistence flows only there, and the 5-pixel border of
    reference pixels of WFC3-IR raw/ima frames gives and receives none.
    Frames of other detectors, or with no pixel in common, are refused.

    The output has CURRENT's structure and units, with provenance and
    checksums in its primary header; ERR and DQ change as --model-error and
    --flag-above say.

    \b
    Examples:
      perscli apply-persistence sample_data/exp4.fits sample_data/exp1.fits sample_data/exp2.fits \\
          sample_data/exp3.fits -o exp4_pers.fits
      perscli apply-persistence sample_data/exp4.fits sample_data/exp3.fits --mode predict -o pers.fits
      perscli apply-persistence sample_data/exp4.fits sample_data/exp3.fits --law pessimistic \\
          --set persistence.gamma=1.1 -o exp4_pess.fits
      perscli apply-persistence exp4_pers.fits sample_data/exp1.fits sample_data/exp2.fits sample_data/exp3.fits \\
          --mode subtract --flag-above 0.01 -o exp4_corr.fits
      perscli apply-persistence sample_data/exp4.fits sample_data/exp1.fits sample_data/exp2.fits \\
          sample_data/exp3.fits --law wfc3 --mode predict -o pers_wfc3.fits
      perscli apply-persistence sample_data/exp4.fits 'sample_data/exp3.fits[SCI][65:192,65:192]' --mode predict \\
          -o pers_cutout.fits
      cat sample_data/exp4.fits | perscli apply-persistence - sample_data/exp3.fits -o - \\
          | perscli apply-persistence - sample_data/exp2.fits -o out.fits

    (sample_data/ is in the clone: four 256 x 256 exposures of one field,
    139.8 s each, 30 s apart; the fourth example corrects the first's
    output.)
    """
    from ..detector.apply import apply_persistence_files
    from ..detector.model import load_persistence_model

    if law is not None and model_spec is not None:
        raise click.UsageError("--law and --model name the same thing (--model is its older spelling): give --law")
    law = law if law is not None else model_spec if model_spec is not None else "typical"
    if dq_bit is not None and flag_above is None:
        raise click.UsageError("--dq-bit sets the bit --flag-above flags: give --flag-above E_PER_S too")
    check_outputs(output, inputs=[current, *previous, law], overwrite=overwrite)
    # whole frames made and dropped over and over: kept for reuse rather than mapped afresh each time
    keep_freed_memory()
    # the options --time-model, --combine, --max-previous and --lookback are the law's settings
    # --set persistence.KEY=VALUE arrives as KEY=VALUE (options.key_values), as the older --param gives it
    model = load_persistence_model(law, (*settings, *params)).with_settings(
        time_model=time_model, combine=combine, max_previous=max_previous, lookback=lookback)
    options = ApplyOptions(mode=mode, model_error=model_error, flag_above=flag_above,
                           dq_bit=D.dq_bit if dq_bit is None else dq_bit, units=units, gain=gain, exptime=exptime,
                           gap=gap, compress=compress)
    result = apply_persistence_files(current, previous, output, model=model, options=options, overwrite=overwrite,
                                     workers=workers, progress=progress_reporter("blocks of rows", least=PROGRESS_LEAST))
    log.info("%s: persistence from %d earlier exposure(s): max %.4g e-, total %.6g e- (last plane)%s",
             "stdout" if output == "-" else output, len(result.used), result.max_electrons,
             result.total_electrons, f"; {result.flagged} pixel(s) flagged in DQ" if flag_above is not None else "")
