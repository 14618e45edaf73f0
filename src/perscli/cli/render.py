"""``perscli render``: a Roman SCA exposure of a truth catalogue, through a detector model."""

from __future__ import annotations

import logging
import shutil

import click

from .. import PerscliError
from ..executor import keep_freed_memory
from ..instrument import ROMAN_EXPTIME, ROMAN_FILTERS, ROMAN_N_SCA, ROMAN_SCA_SIZE
from ..io.config import DETECTOR_ITEM
from ..render.settings import DEFAULT_HDUS, HDU_NAMES, RenderOptions
from ..scene import check_filter
from .helpers import FILE, PerscliCommand, check_outputs, progress_reporter, report_errors
from .options import (chosen_seed_option, columns_opt, compress_option, dec_opt, key_values, mjd_opt, model_opt,
                      no_checksum_opt, output_option, overwrite_opt, pa_opt, plot_opt, ra_opt, settings_options,
                      verbosity_opts, workers_opt)

log = logging.getLogger("perscli")

#: work below this many steps tells a log (stderr not a terminal) nothing: a full SCA draws thousands of objects
#: (minutes), a cutout's few dozen take seconds
PROGRESS_LEAST = 1000

#: the defaults, written once (perscli.render.settings)
D = RenderOptions()


def _list_effects(ctx, param, value):
    """--list-effects: print the registry's schema and stop (no TRUTH.fits, --seed or -o needed)."""
    if not value or ctx.resilient_parsing:
        return
    from ..detector.model import format_schema

    click.echo(format_schema(width=max(100, shutil.get_terminal_size((120, 24)).columns)), nl=False)
    ctx.exit(0)


@click.command("render", cls=PerscliCommand,
               short_help="Draw a Roman SCA exposure of a truth catalogue through a detector model.")
@click.argument("truth", metavar="TRUTH.fits", type=FILE)
@click.option("--pointings", "pointings_file", metavar="FILE", type=FILE,
              help="A pointings table (perscli pointings) or a survey schedule (date, exptime, ra, dec, pa, "
                   "filter) to take the exposure from; see --row.")
@click.option("--row", type=click.IntRange(min=0), default=0, show_default=True, metavar="N",
              help="Row of --pointings (0 is the first; for a schedule, its row number).")
@ra_opt("Pointing centre of the focal plane (instead of --pointings, or overriding it): right ascension")
@dec_opt("Pointing centre of the focal plane: declination")
@pa_opt("Observatory position angle, degrees (GalSim's convention).")
@mjd_opt("--mjd", "Start of the exposure; Roman must be able to point there then (54 to 126 degrees from the Sun).")
@click.option("--exptime", type=click.FloatRange(min=0, min_open=True), metavar="SECONDS",
              help=f"Exposure time [default: {ROMAN_EXPTIME:g}, or the pointing's].")
@click.option("--filter", "filter_name", metavar="NAME", help=f"Roman filter: {' '.join(ROMAN_FILTERS)}.")
@click.option("--sca", type=click.IntRange(1, ROMAN_N_SCA), metavar="N",
              help=f"Detector 1-{ROMAN_N_SCA} (default: the pointing's sca column).")
@click.option("--bounds", type=int, nargs=4, metavar="XMIN XMAX YMIN YMAX",
              help="Render a cutout: 1-indexed inclusive SCA pixels "
                   f"[default: the full {ROMAN_SCA_SIZE} x {ROMAN_SCA_SIZE}].")
@model_opt("roman", "roman|MODEL.yaml|FRAME.fits",
           "roman (GalSim's Roman chain, with saturation), a YAML list of effects in physical order, or a frame "
           "perscli rendered (the model that made it); see --list-effects", names=("roman",))
@click.option("--set", "settings", multiple=True, metavar="EFFECT.KEY=VALUE", callback=key_values(DETECTOR_ITEM),
              help="Override the model: e.g. read_noise.sigma=5, persistence.base=pessimistic, ipc=off.")
@click.option("--previous", multiple=True, metavar="FRAME", type=FILE,
              help="An earlier exposure of the same SCA (a frame perscli rendered); repeatable. Its DRAWN "
                   "(STARFLU for --persistence-source stars, FLUENCE for all) leaves persistence in this one.")
@click.option("--persistence-source", "persistence_source", metavar="drawn|stars|all|ELECTRONS",
              default=D.persistence_source,
              help="What of the --previous frames persists: drawn (their DRAWN: the light drawn on them, galaxies "
                   "and stars, no sky: the paper's pipeline and perscli study's headline), stars (their STARFLU: "
                   "the light of stars only), all (their FLUENCE: every photon, the sky's too) or a number of "
                   "electrons (only pixels whose FLUENCE exceeds it); same as --set persistence.source=...  "
                   "[default: the model's, drawn]")
@click.option("--hdus", metavar="NAME,...", default=",".join(D.hdus),
              help=f"The HDUs to write, among {','.join(HDU_NAMES)} (DRAWN: the light drawn, what later "
                   "frames' persistence comes from by default)  "
                   f"[default: {','.join(DEFAULT_HDUS)}]")
@click.option("--dry-run", "dry_run", is_flag=True, default=False,
              help="Draw nothing, write no frame or figure (no -o or --seed needed): print where the frame lands (its "
                   "corners on the sky, its size) and how many stars and galaxies of TRUTH.fits land on it.")
@click.option("--regions", metavar="FILE.reg", default=None, type=FILE,
              help="With --dry-run: also write a ds9 region file (fk5) of the frame's outline and of the objects "
                   "drawn on it.")
@settings_options(RenderOptions, "strict")
@columns_opt("TRUTH.fits", "ra=ALPHA_J2000,dec=DELTA_J2000,id=NUMBER")
# --dry-run draws and writes nothing: -o and --seed are required only without it, which the body checks
# (usage errors, exit 2, in click's own words)
@chosen_seed_option(required=False)
@plot_opt("the frame and its persistence")
@click.option("--list-effects", is_flag=True, expose_value=False, is_eager=True, callback=_list_effects,
              help="Print every effect's parameters (type, unit, default, allowed values) and exit.")
@output_option(required=False)
@compress_option(D.compress)
@no_checksum_opt
@overwrite_opt
@workers_opt("processes drawing the objects' stamps (the output does not depend on N)")
@verbosity_opts
@report_errors
def render(truth, pointings_file, row, ra, dec, pa, mjd, exptime, filter_name, sca, bounds, model_spec, settings,
           previous, persistence_source, hdus, dry_run, regions, strict, columns, seed, plot, output, compress, overwrite,
           workers):
    """Draw a Roman SCA exposure of TRUTH.fits through a detector model.

    Optics from GalSim's Roman module: the SCA's WCS for the pointing, its PSF
    for the filter (at the SCA centre and the filter's effective wavelength),
    the filter's AB zeropoint and the zodiacal (on the exposure's date) plus
    thermal sky.  Stamps grow with flux so that bright stars keep their
    diffraction spikes, the source of their persistence ghosts.  The detector chain (sky, Poisson noise,
    reciprocity failure, dark current, persistence, saturation at the full
    well, nonlinearity, IPC, read noise, gain, quantisation) follows the model
    (--list-effects prints every parameter); each effect has its own random
    stream, so frames rendered with and without persistence share their noise.

    The output has SCI (the frame, DN after gain), IDEAL (noise-free electrons
    from sky and sources), FLUENCE (the charge collected, at most the full
    well), DRAWN (the noise-free electrons of every object drawn, galaxies and
    stars, no sky, not clipped at the well), STARFLU (the same of the stars
    alone, on request), with --previous PERSIST (electrons of persistence), and
    MODEL (the resolved detector model, which --model FRAME.fits reads
    back); WCS, timing, SCA, FILTER and GAIN in the headers.  --hdus
    chooses among them.

    What of the --previous frames persists (--persistence-source): their
    DRAWN (drawn, the default: every object's light, galaxies and stars, no
    sky, as the paper's pipeline persisted it), their STARFLU (stars: the
    stars' light alone), all their FLUENCE (the sky's light too: in frames
    rounded to whole DN, a sky-level halo of ~1e-4 of the sky that flips
    pixels by one DN), or the FLUENCE of pixels above a number of
    electrons; the fluence fed to the persistence law is capped at
    persistence.fluence_cap when one is set (default none: the law
    extrapolated beyond the well, as GalSim's applyPersistence does).  A
    frame rendered with the default HDUs serves as the history of later
    frames for the sources drawn and all; add STARFLU for stars.

    The exposure (pointing, PA, date, filter) comes from a row of
    --pointings or from --ra --dec --pa --mjd --filter; Roman must be able
    to point there on that date (GalSim: 54 to 126 degrees from the Sun),
    or render stops with one line naming the first date it can.  The SCA
    lies up to 0.45 degrees from the pointing, not at it: --dry-run prints
    where the frame lands and how many objects of TRUTH.fits it covers,
    drawing nothing; a frame on which no object lands is warned about
    (naming where the frame and the catalogue are), and refused with
    --strict.  perscli pointings select|plan --footprints --catalog counts the objects
    on every row, and perscli catalog --pointings draws a catalogue where
    the SCA lands.

    \b
    Examples:
      perscli pointings plan --ra 10 --dec -44 --n 3 --sca 7 -o seq.fits
      perscli catalog --pointings seq.fits --bounds 1 512 1 512 -o seq_truth.fits
      perscli render seq_truth.fits --pointings seq.fits --row 0 --bounds 1 512 1 512 --dry-run --regions seq0.reg
      perscli render seq_truth.fits --pointings seq.fits --row 0 --bounds 1 512 1 512 --seed 1 --strict -o e0.fits
      perscli render seq_truth.fits --pointings seq.fits --row 1 --bounds 1 512 1 512 --seed 2 --previous e0.fits \\
          -o e1.fits
      perscli render seq_truth.fits --pointings seq.fits --row 1 --bounds 1 512 1 512 --seed 2 --set persistence=off \\
          -o e1_nop.fits
      perscli render seq_truth.fits --pointings seq.fits --row 2 --bounds 1 512 1 512 --seed 3 --model e1.fits \\
          -o e2.fits
      perscli render seq_truth.fits --pointings seq.fits --row 0 --bounds 1 512 1 512 --seed 1 \\
          --hdus SCI,FLUENCE,STARFLU --compress gzip -o h0.fits
      perscli render seq_truth.fits --pointings seq.fits --row 1 --bounds 1 512 1 512 --seed 2 --previous h0.fits \\
          --persistence-source all --hdus SCI,PERSIST -o e1_all.fits
      perscli catalog --ra 9.5 --dec -44.06 --size 10 -o sca7_truth.fits
      perscli render sca7_truth.fits --ra 10 --dec -44 --pa 30 --mjd 61541.97 --filter J129 --sca 7 \\
          --bounds 1 512 1 512 --model sample_data/roman_detector.yaml --set read_noise.sigma=5 --seed 4 --plot explicit.png \\
          -o explicit.fits
      perscli render --list-effects
    """
    from ..detector.model import load_detector_model
    from ..render.run import (footprint_report, format_footprint, no_objects_fix, no_objects_message, render_file,
                              write_regions)

    if regions is not None and not dry_run:
        raise click.UsageError("--regions is written by --dry-run: add --dry-run (or drop --regions)")
    if not dry_run:
        if output is None:
            raise click.UsageError("Missing option '-o' / '--output' (only --dry-run writes no frame).")
        if seed is None:
            raise click.UsageError("Missing option '--seed' (only --dry-run draws nothing).")
    if dry_run:
        if regions is not None:
            check_outputs(regions, inputs=[truth, pointings_file, model_spec, *previous], overwrite=overwrite,
                          fits=False)
        exposure = _exposure(pointings_file, row, ra, dec, pa, mjd, exptime, filter_name, sca, bounds)
        load_detector_model(model_spec, settings)          # a dry run checks what the run would check
        report = footprint_report(truth, exposure, columns=columns)
        if len(report["drawn"]) == 0:
            message = no_objects_message(report, dry_run=True)
            if strict:
                raise PerscliError("--strict: " + message)
            log.warning("%s%s", message, no_objects_fix(dry_run=True))
        source = f"{pointings_file} row {row}" if pointings_file is not None else ""
        if regions is not None:
            write_regions(report, regions, overwrite=overwrite)
        click.echo(format_footprint(report, source=source), nl=False)
        if output is not None:
            log.info("--dry-run: %s not written", output)
        return
    check_outputs(output, inputs=[truth, pointings_file, model_spec, *previous], plot=plot, overwrite=overwrite)
    # whole frames made and dropped over and over: kept for reuse rather than mapped afresh each time
    keep_freed_memory()
    exposure = _exposure(pointings_file, row, ra, dec, pa, mjd, exptime, filter_name, sca, bounds)
    model = load_detector_model(model_spec, settings)
    options = RenderOptions(hdus=hdus, compress=compress, persistence_source=persistence_source, strict=strict,
                            columns=columns)
    summary = render_file(truth, exposure, output, options, model=model, seed=seed, previous=previous,
                          overwrite=overwrite, workers=workers, plot=plot,
                          progress=progress_reporter("objects", least=PROGRESS_LEAST))
    log.info("%s: %d objects, sky %.3f e-/pixel/s, units %s, persistence max %.3g e-",
             "stdout" if output == "-" else output, summary["objects"], summary["sky_rate"], summary["unit"],
             summary["persistence_max"])


def _exposure(pointings_file, row, ra, dec, pa, mjd, exptime, filter_name, sca, bounds):
    from ..render.exposure import Exposure
    from ..scene.pointings import read_pointings

    explicit = {"--ra": ra, "--dec": dec, "--pa": pa, "--mjd": mjd, "--filter": filter_name}
    if pointings_file is not None:
        table = read_pointings(pointings_file)
        if row >= len(table):
            raise PerscliError(f"{pointings_file}: --row {row} is past the end ({len(table)} rows)")
        p = table[row]
        values = {"--ra": p.ra, "--dec": p.dec, "--pa": p.pa, "--mjd": p.mjd, "--filter": p.filter}
        values.update({k: v for k, v in explicit.items() if v is not None})
        exptime = exptime if exptime is not None else p.exptime
        sca = sca if sca is not None else (p.sca or None)
        expid = p.expid
    else:
        missing = [k for k, v in explicit.items() if v is None]
        if missing:
            raise click.UsageError(f"give --pointings FILE, or all of --ra --dec --pa --mjd --filter "
                                   f"(missing {' '.join(missing)})")
        values, expid = explicit, -1
    if sca is None:
        raise click.UsageError(f"give --sca N (1-{ROMAN_N_SCA}): the pointing does not name a detector")
    return Exposure(ra=values["--ra"], dec=values["--dec"], pa=values["--pa"], sca=sca,
                    filter=check_filter(values["--filter"]), mjd=values["--mjd"],
                    exptime=exptime if exptime is not None else ROMAN_EXPTIME,
                    bounds=tuple(bounds) if bounds else None, expid=expid)
